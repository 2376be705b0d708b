"""The patient tracker's per-tick maths, compiled (numba): the string lengths and their
Jacobian, one Gauss-Newton update of the tooth's pose, and the rotation vector of a rotation
matrix (its log map) with its inverse (Rodrigues' formula).

:mod:`dentibot.control.strings` (the model, its forward kinematics and calibration) and
:mod:`dentibot.runtime.tooth` (the tracked tooth of the control tick) call these, and the
Meca500 simulator's inverse kinematics takes its orientation error from :func:`matrix_rotvec`;
they are the only implementation of the strings' formulas and of the log map (the simulated
patient's turns keep Rodrigues' formula in a scalar form of their own,
:func:`dentibot.sim.patient.axis_angle_matrix`, for a world tick without arrays)::

    l_i = || d_i ||,   d_i = p + R b_i - a_i,   u_i = d_i / l_i
    J_i = [u_i, (R b_i) x u_i]                       (dl = J (dp, dth), R <- exp([dth]x) R)
    exp([r]x) = I + sin(t)/t [r]x + (1 - cos(t))/t^2 [r]x^2,   t = ||r||

Compiled at import, as :mod:`~dentibot.control.kinematics_kernels` explains: a tracked tick
runs these at every control period.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def lengths(a: np.ndarray, b: np.ndarray, R: np.ndarray, p: np.ndarray) -> np.ndarray:
    """``l_i = || p + R b_i - a_i ||`` (mm) for anchors ``a`` (n x 3, {M}) and ``b``
    (n x 3, {T}) at the pose ``(R, p)``."""
    n = a.shape[0]
    out = np.empty(n)
    for i in range(n):
        s = 0.0
        for r in range(3):
            d = p[r] + R[r, 0] * b[i, 0] + R[r, 1] * b[i, 1] + R[r, 2] * b[i, 2] - a[i, r]
            s += d * d
        out[i] = math.sqrt(s)
    return out


@njit(cache=True)
def jacobian(a: np.ndarray, b: np.ndarray, R: np.ndarray, p: np.ndarray) -> np.ndarray:
    """The lengths' Jacobian ``J`` (n x 6): row ``[u_i, (R b_i) x u_i]``."""
    n = a.shape[0]
    out = np.empty((n, 6))
    rb = np.empty(3)
    u = np.empty(3)
    for i in range(n):
        s = 0.0
        for r in range(3):
            rb[r] = R[r, 0] * b[i, 0] + R[r, 1] * b[i, 1] + R[r, 2] * b[i, 2]
            u[r] = p[r] + rb[r] - a[i, r]
            s += u[r] * u[r]
        norm = math.sqrt(s)
        for r in range(3):
            u[r] /= norm
            out[i, r] = u[r]
        out[i, 3] = rb[1] * u[2] - rb[2] * u[1]
        out[i, 4] = rb[2] * u[0] - rb[0] * u[2]
        out[i, 5] = rb[0] * u[1] - rb[1] * u[0]
    return out


@njit(cache=True)
def rotvec_matrix(r: np.ndarray) -> np.ndarray:
    """``exp([r]x)``: the rotation matrix of the rotation vector ``r`` (rad), Rodrigues'
    formula (its series below 1e-4 rad, exact to rounding there too)."""
    t2 = r[0] * r[0] + r[1] * r[1] + r[2] * r[2]
    t = math.sqrt(t2)
    if t < 1e-4:
        s = 1.0 - t2 / 6.0                       # sin(t)/t
        c = 0.5 - t2 / 24.0                      # (1 - cos(t))/t^2
    else:
        s = math.sin(t) / t
        c = (1.0 - math.cos(t)) / t2
    x, y, z = r[0], r[1], r[2]
    m = np.empty((3, 3))
    m[0, 0] = 1.0 - c * (y * y + z * z)
    m[1, 1] = 1.0 - c * (x * x + z * z)
    m[2, 2] = 1.0 - c * (x * x + y * y)
    m[0, 1] = c * x * y - s * z
    m[1, 0] = c * x * y + s * z
    m[0, 2] = c * x * z + s * y
    m[2, 0] = c * x * z - s * y
    m[1, 2] = c * y * z - s * x
    m[2, 1] = c * y * z + s * x
    return m


@njit(cache=True)
def matrix_rotvec(m: np.ndarray) -> np.ndarray:
    """The rotation vector (rad) of the rotation matrix ``m``, its angle in [0, pi]: the
    angle from ``atan2(|v|, (tr m - 1) / 2)`` with ``v`` the axial vector of
    ``(m - m^T) / 2`` (accurate at small angles, where an arccos of the trace is not); near
    pi, where ``v`` vanishes, the axis from the symmetric part of ``m``."""
    vx = 0.5 * (m[2, 1] - m[1, 2])
    vy = 0.5 * (m[0, 2] - m[2, 0])
    vz = 0.5 * (m[1, 0] - m[0, 1])
    s = math.sqrt(vx * vx + vy * vy + vz * vz)         # sin(angle)
    c = 0.5 * (m[0, 0] + m[1, 1] + m[2, 2] - 1.0)      # cos(angle)
    angle = math.atan2(s, c)
    out = np.empty(3)
    if c > -0.9:                 # angle below about 154 deg: the axial vector is reliable
        k = 1.0 + angle * angle / 6.0 if s < 1e-8 else angle / s
        out[0], out[1], out[2] = k * vx, k * vy, k * vz
        return out
    # near pi: (m + m^T) / 2 - cos(a) I = (1 - cos(a)) n n^T; its column of the largest
    # diagonal term is the axis n (to scale), signed like v
    i = 0
    if m[1, 1] > m[i, i]:
        i = 1
    if m[2, 2] > m[i, i]:
        i = 2
    col = np.empty(3)
    for r in range(3):
        col[r] = 0.5 * (m[r, i] + m[i, r]) - (c if r == i else 0.0)
    norm = math.sqrt(col[0] * col[0] + col[1] * col[1] + col[2] * col[2])
    sign = 1.0 if col[0] * vx + col[1] * vy + col[2] * vz >= 0.0 else -1.0
    for r in range(3):
        out[r] = sign * angle * col[r] / norm
    return out


@njit(cache=True)
def track(a: np.ndarray, b: np.ndarray, m: np.ndarray, R: np.ndarray, p: np.ndarray,
          iterations: int):
    """``iterations`` Gauss-Newton steps of the pose ``(R, p)`` towards the measured lengths
    ``m`` (all strings; the least-squares step of ``J dx = m - l``, then ``p += dx[:3]``,
    ``R <- exp([dx[3:]]x) R``). Returns ``(R, p, rms residual mm)``; a non-finite step (a
    singular Jacobian) gives a non-finite residual."""
    R = R.copy()
    p = p.copy()
    for _ in range(iterations):
        r = m - lengths(a, b, R, p)
        dx = np.linalg.lstsq(jacobian(a, b, R, p), r)[0]
        for k in range(3):
            p[k] += dx[k]
        R = rotvec_matrix(dx[3:].copy()) @ R
    res = m - lengths(a, b, R, p)
    return R, p, math.sqrt(np.mean(res * res))


def warm_up() -> None:
    """Compile (or load from the cache) every kernel for the types its callers pass: the
    anchors of a :class:`~dentibot.control.strings.StringGeometry` are read-only arrays, the
    pose and lengths writable copies. Called once, at import."""
    from dentibot.control.linalg import readonly

    a = readonly(np.eye(6, 3) * 50.0 + 1.0)
    b = readonly(np.eye(6, 3) * 10.0)
    eye, p = np.eye(3), np.zeros(3)
    lengths(a, b, eye, p)
    jacobian(a, b, eye, p)
    track(a, b, np.ones(6) * 40.0, eye, p, 1)
    rotvec_matrix(p)
    matrix_rotvec(eye)


warm_up()      # at import: before any device streams or loop runs
