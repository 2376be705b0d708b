"""From the admittance twist to the joint command, compiled (numba): the joint rates (exact
solve, or damped least squares near a singularity), the limits of thesis 4.3 and the
trapezoidal integration to the joint target (fig 4.2).

:class:`~dentibot.control.admittance.AdmittanceController` and
:class:`~dentibot.control.limits.JointLimiter` call these; they are the only implementation.
Each kernel works on one arm. Units: joint angles deg, joint rates rad/s.

``thresholds`` is the limiter's singularity table as an array: ``(shoulder_stop_mm,
shoulder_start_mm, elbow_stop, elbow_start, wrist_stop, wrist_start)``; ``sing`` the six
singularity factors and rates of :func:`~dentibot.control.kinematics_kernels.singularity_factors`.

Compiled at import, as :mod:`~dentibot.control.kinematics_kernels` explains.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from dentibot.control.kinematics_kernels import singularity_factors

#: Above this normalised singularity factor the joint rates are the exact solution.
EXACT_SOLVE_ABOVE = 0.2


@njit(cache=True)
def damped_least_squares(j: np.ndarray, v: np.ndarray, sigma_min_ok: float = 0.05,
                         lambda_max: float = 0.05) -> np.ndarray:
    """Solve ``J qdot = v`` with damping that grows smoothly near a singularity.

    Far from singularities (smallest singular value >= ``sigma_min_ok``) this is the exact
    solution. Closer, ``lambda^2 = (1 - (s/sigma_min_ok)^2) lambda_max^2`` (Nakamura, Chiaverini)
    trades tracking accuracy for bounded joint rates: the result never blows up.
    """
    u, s, vt = np.linalg.svd(j)
    smin = s[-1]
    if smin >= sigma_min_ok:
        lam2 = 0.0
    else:
        lam2 = (1.0 - (smin / sigma_min_ok) ** 2) * lambda_max**2
    return vt.T @ ((s / (s * s + lam2)) * (u.T @ v))


@njit(cache=True)
def _ramp(value: float, stop: float, start: float) -> float:
    if value >= start:
        return 1.0
    if value <= stop:
        return 0.0
    return (value - stop) / (start - stop)


@njit(cache=True)
def singularity_scale(sing, thresholds: np.ndarray) -> float:
    """Each factor below its start threshold *and decreasing* scales the rates down, to zero
    at its stop threshold; moving away from a singularity is never slowed."""
    scale = 1.0
    if sing[3] < 0.0:
        scale = min(scale, _ramp(sing[0], thresholds[0], thresholds[1]))
    if sing[4] < 0.0:
        scale = min(scale, _ramp(sing[1], thresholds[2], thresholds[3]))
    if sing[5] < 0.0:
        scale = min(scale, _ramp(sing[2], thresholds[4], thresholds[5]))
    return scale


@njit(cache=True)
def limit_rates(q_deg: np.ndarray, qdot_rad_s: np.ndarray, sing, thresholds: np.ndarray,
                lo_rad: np.ndarray, hi_rad: np.ndarray, vmax_rad_s: np.ndarray,
                margin_rad: float, ts: float):
    """The limits of :class:`~dentibot.control.limits.JointLimiter`: ``(qdot, singularity
    scale, speed scale, guarded)`` (``guarded``: per joint, clamped by its range)."""
    s_scale = singularity_scale(sing, thresholds)
    out = np.empty(6)
    guarded = np.zeros(6, np.bool_)
    ratio = 0.0
    for i in range(6):
        w = qdot_rad_s[i] * s_scale if s_scale < 1.0 else qdot_rad_s[i]
        qi = math.radians(q_deg[i])
        dist = max(hi_rad[i] - qi if w > 0.0 else qi - lo_rad[i], 0.0)
        vmax = vmax_rad_s[i]
        if dist < margin_rad:
            allowed = min(vmax * dist / margin_rad, dist / ts)
            if abs(w) > allowed:
                w = math.copysign(allowed, w)
                guarded[i] = True
        out[i] = w
        ratio = max(ratio, abs(w) / vmax)
    speed_scale = 1.0
    if ratio > 1.0:
        speed_scale = 1.0 / ratio
        for i in range(6):
            out[i] *= speed_scale
    return out, s_scale, speed_scale, guarded


@njit(cache=True)
def joint_step(jh: np.ndarray, twist: np.ndarray, frames: np.ndarray, q_deg: np.ndarray,
               w_prev: np.ndarray, half_ts_deg: float, q_lo: np.ndarray, q_hi: np.ndarray,
               singular_sigma: float, elbow_offset: float, wrist_frame: int,
               thresholds: np.ndarray, lo_rad: np.ndarray, hi_rad: np.ndarray,
               vmax_rad_s: np.ndarray, margin_rad: float, ts: float):
    """One period from the twist (mm/s, rad/s in {H}; ``jh`` its Jacobian at ``q_deg``):
    the joint rates (the exact solve when the worst singularity factor is above
    :data:`EXACT_SOLVE_ABOVE`, else damped least squares with ``singular_sigma``), limited,
    and the joint target ``q + ts/2 (qdot + qdot_prev)`` within the joint ranges.

    Returns ``(q_next_deg, qdot_rad_s, sing, singularity scale, speed scale, guarded)``."""
    s0 = singularity_factors(frames, q_deg, w_prev, False, elbow_offset, wrist_frame)
    if min(s0[0] / 50.0, s0[1], s0[2], 1.0) > EXACT_SOLVE_ABOVE:
        qdot = np.linalg.solve(jh, twist)
    else:
        qdot = damped_least_squares(jh, twist, singular_sigma)
    sing = singularity_factors(frames, q_deg, qdot, True, elbow_offset, wrist_frame)
    out, s_scale, speed_scale, guarded = limit_rates(q_deg, qdot, sing, thresholds, lo_rad,
                                                     hi_rad, vmax_rad_s, margin_rad, ts)
    q_next = np.empty(6)
    for i in range(6):
        q_next[i] = min(max(q_deg[i] + half_ts_deg * (out[i] + w_prev[i]), q_lo[i]), q_hi[i])
    return q_next, out, sing, s_scale, speed_scale, guarded


def warm_up() -> None:
    """Compile (or load from the cache) every kernel of this module for the argument types
    the admittance controller, the limiter and the simulated arm's inverse kinematics pass
    (see :func:`dentibot.control.kinematics_kernels.warm_up`). Called once, at import."""
    from dentibot.control.kinematics_kernels import dh_frames

    dh = np.zeros((6, 5))
    dh[:, 0] = 1.0
    q, one = np.zeros(6), np.ones(6)
    frames = dh_frames(dh, q)
    th = np.array([5.0, 20.0, 0.03, 0.17, 0.03, 0.17])
    joint_step(np.eye(6), one, frames, q, q, 0.06, -one, one, 0.05, 0.0, 4, th, -one, one,
               one, 0.1, 0.002)
    limit_rates(q, one, (1.0, 1.0, 1.0, 0.0, 0.0, 0.0), th, -one, one, one, 0.1, 0.002)
    singularity_scale((1.0, 1.0, 1.0, 0.0, 0.0, 0.0), th)
    # explicit and omitted defaults are two signatures to numba: both are called
    damped_least_squares(np.eye(6), one, 0.05, 0.05)
    damped_least_squares(np.eye(6), one)


warm_up()      # at import: before any device streams or loop runs
