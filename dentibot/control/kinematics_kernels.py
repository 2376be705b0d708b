"""The Meca500's forward chain, tool Jacobian and singularity measures, compiled (numba).

:class:`~dentibot.control.kinematics.Meca500` calls these every tick (the controller once,
the simulated arm once); they are the only implementation of the chain. A chain is an array
``frames`` of shape (6, 4, 3): for joint frame i (0-based), ``frames[i, 0:3]`` its rotation's
columns x, y, z in {0} and ``frames[i, 3]`` its origin (mm).

The link table ``dh`` has one row per joint: ``(cos alpha, sin alpha, a, theta offset rad,
d)`` of the modified (Craig) convention, ``Rx(alpha_{i-1}) Tx(a_{i-1}) Rz(theta_i) Tz(d_i)``
(thesis Table 3.1). Each kernel works on one arm; a population of arms calls them in a loop
inside compiled code.

The kernels are compiled (or loaded from numba's cache, next to this file) when the module is
imported (:func:`warm_up`): a process connects its devices after its imports, and a control
loop must not pay a compilation (100 ms and more) at its first tick, when the drive's 30 ms
heartbeat consumer is already watching. The first import after a change compiles them (a few
seconds).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_RAD = math.pi / 180.0


@njit(cache=True)
def dh_frames(dh: np.ndarray, q_deg: np.ndarray) -> np.ndarray:
    """Frames {1}..{6} in {0} at joint angles ``q_deg`` (deg), shape (6, 4, 3).

    Each link is ``R <- R Rx(alpha) Rz(theta)``, ``p <- p + a x + d z'``, propagated column by
    column (``Rx(alpha) Rz(theta)`` has a fixed structure)."""
    out = np.empty((6, 4, 3))
    x0, x1, x2 = 1.0, 0.0, 0.0
    y0, y1, y2 = 0.0, 1.0, 0.0
    z0, z1, z2 = 0.0, 0.0, 1.0
    p0 = p1 = p2 = 0.0
    for i in range(6):
        ca, sa, a, off, d = dh[i, 0], dh[i, 1], dh[i, 2], dh[i, 3], dh[i, 4]
        # R Rx(alpha): y' = ca y + sa z, z' = -sa y + ca z
        u0, u1, u2 = ca * y0 + sa * z0, ca * y1 + sa * z1, ca * y2 + sa * z2
        z0, z1, z2 = -sa * y0 + ca * z0, -sa * y1 + ca * z1, -sa * y2 + ca * z2
        p0 += a * x0 + d * z0
        p1 += a * x1 + d * z1
        p2 += a * x2 + d * z2
        th = q_deg[i] * _RAD + off
        ct, st = math.cos(th), math.sin(th)
        # Rz(theta): x'' = ct x + st y', y'' = -st x + ct y'
        x0, x1, x2, y0, y1, y2 = (ct * x0 + st * u0, ct * x1 + st * u1, ct * x2 + st * u2,
                                  -st * x0 + ct * u0, -st * x1 + ct * u1, -st * x2 + ct * u2)
        out[i, 0, 0], out[i, 0, 1], out[i, 0, 2] = x0, x1, x2
        out[i, 1, 0], out[i, 1, 1], out[i, 1, 2] = y0, y1, y2
        out[i, 2, 0], out[i, 2, 1], out[i, 2, 2] = z0, z1, z2
        out[i, 3, 0], out[i, 3, 1], out[i, 3, 2] = p0, p1, p2
    return out


@njit(cache=True)
def _mul_cols(f: np.ndarray, k: int, a: float, b: float, c: float):
    """R_k @ (a, b, c) for the rotation of frame ``k`` of ``f`` (columns)."""
    return (f[k, 0, 0] * a + f[k, 1, 0] * b + f[k, 2, 0] * c,
            f[k, 0, 1] * a + f[k, 1, 1] * b + f[k, 2, 1] * c,
            f[k, 0, 2] * a + f[k, 1, 2] * b + f[k, 2, 2] * c)


@njit(cache=True)
def tool_point_axes(frames: np.ndarray, tool: np.ndarray, ref_h: np.ndarray) -> np.ndarray:
    """The point ``ref_h`` of {H} (mm, in {H}; ``tool`` = 6T_H, 4x4) and the axes of {H}, in
    {0}: shape (4, 3), rows x_H, y_H, z_H, point."""
    out = np.empty((4, 3))
    tp0, tp1, tp2 = tool[0, 3], tool[1, 3], tool[2, 3]
    # p_h = tool_p + tool_R @ ref_h (columns of tool_R)
    r0, r1, r2 = ref_h[0], ref_h[1], ref_h[2]
    q0 = tool[0, 0] * r0 + tool[0, 1] * r1 + tool[0, 2] * r2
    q1 = tool[1, 0] * r0 + tool[1, 1] * r1 + tool[1, 2] * r2
    q2 = tool[2, 0] * r0 + tool[2, 1] * r1 + tool[2, 2] * r2
    ph0, ph1, ph2 = tp0 + q0, tp1 + q1, tp2 + q2
    m0, m1, m2 = _mul_cols(frames, 5, ph0, ph1, ph2)
    out[3, 0], out[3, 1], out[3, 2] = frames[5, 3, 0] + m0, frames[5, 3, 1] + m1, \
        frames[5, 3, 2] + m2
    for k in range(3):
        a0, a1, a2 = _mul_cols(frames, 5, tool[0, k], tool[1, k], tool[2, k])
        out[k, 0], out[k, 1], out[k, 2] = a0, a1, a2
    return out


@njit(cache=True)
def point_jacobian(frames: np.ndarray, point: np.ndarray, axes: np.ndarray,
                   in_axes: bool) -> np.ndarray:
    """Geometric Jacobian (6x6) for the velocity of ``point`` (in {0}) (eq 3.5-3.7): column i
    is ``(z_i x (p - o_i), z_i)``; with ``in_axes`` its rows are expressed in the frame whose
    axes (in {0}) are the rows of ``axes`` (eq 3.10-3.14)."""
    j = np.empty((6, 6))
    px, py, pz = point[0], point[1], point[2]
    for i in range(6):
        zx, zy, zz = frames[i, 2, 0], frames[i, 2, 1], frames[i, 2, 2]
        dx, dy, dz = px - frames[i, 3, 0], py - frames[i, 3, 1], pz - frames[i, 3, 2]
        lx, ly, lz = zy * dz - zz * dy, zz * dx - zx * dz, zx * dy - zy * dx
        if not in_axes:
            j[0, i], j[1, i], j[2, i], j[3, i], j[4, i], j[5, i] = lx, ly, lz, zx, zy, zz
        else:
            for r in range(3):
                j[r, i] = axes[r, 0] * lx + axes[r, 1] * ly + axes[r, 2] * lz
                j[3 + r, i] = axes[r, 0] * zx + axes[r, 1] * zy + axes[r, 2] * zz
    return j


@njit(cache=True)
def singularity_factors(frames: np.ndarray, q_deg: np.ndarray, qdot_rad_s: np.ndarray,
                        with_rates: bool, elbow_offset: float, wrist_frame: int):
    """The three singularity factors and, ``with_rates``, their rates of change under the
    joint rates ``qdot_rad_s``: ``(shoulder_mm, elbow, wrist, shoulder_rate, elbow_rate,
    wrist_rate)`` (see :class:`~dentibot.control.kinematics.SingularityMeasure`)."""
    w0, w1, w2 = frames[wrist_frame, 3, 0], frames[wrist_frame, 3, 1], frames[wrist_frame, 3, 2]
    rho = math.hypot(w0, w1)
    elbow_angle = math.radians(q_deg[2]) - elbow_offset
    elbow = abs(math.cos(elbow_angle))
    q5 = math.radians(q_deg[4])
    wrist = abs(math.sin(q5))
    if not with_rates:
        return rho, elbow, wrist, 0.0, 0.0, 0.0
    # wrist-centre velocity: only joints 1-3 move it
    v0 = 0.0
    v1 = 0.0
    for i in range(3):
        zx, zy, zz = frames[i, 2, 0], frames[i, 2, 1], frames[i, 2, 2]
        qd = qdot_rad_s[i]
        v0 += (zy * (w2 - frames[i, 3, 2]) - zz * (w1 - frames[i, 3, 1])) * qd
        v1 += (zz * (w0 - frames[i, 3, 0]) - zx * (w2 - frames[i, 3, 2])) * qd
    if rho > 1e-9:
        rho_rate = (w0 * v0 + w1 * v1) / rho
    else:
        rho_rate = -math.hypot(v0, v1)
    elbow_rate = -math.copysign(1.0, math.cos(elbow_angle)) * math.sin(elbow_angle) \
        * qdot_rad_s[2]
    wrist_rate = math.copysign(1.0, math.sin(q5)) * math.cos(q5) * qdot_rad_s[4]
    return rho, elbow, wrist, rho_rate, elbow_rate, wrist_rate


@njit(cache=True)
def euler_xyz_deg(R: np.ndarray) -> tuple[float, float, float]:
    """Mobile XYZ Euler angles (deg) of the rotation matrix ``R`` (3x3), as scipy's
    ``as_euler("XYZ")`` gives them, in closed form: ``R = Rx(a) Ry(b) Rz(g)`` has
    ``R[0, 2] = sin b``, ``R[1, 2] = -sin a cos b``, ``R[2, 2] = cos a cos b``,
    ``R[0, 1] = -cos b sin g``, ``R[0, 0] = cos b cos g``. At ``cos b = 0`` g is 0 and
    ``a = atan2(R[2, 1], R[1, 1])`` (the Meca500's own convention at beta = +-90 deg)."""
    sb = max(-1.0, min(1.0, R[0, 2]))
    b = math.asin(sb)
    if math.hypot(R[0, 0], R[0, 1]) > 1e-9:
        a = math.atan2(-R[1, 2], R[2, 2])
        g = math.atan2(-R[0, 1], R[0, 0])
    else:
        a, g = math.atan2(R[2, 1], R[1, 1]), 0.0
    return math.degrees(a), math.degrees(b), math.degrees(g)


@njit(cache=True)
def tool_euler_deg(frames: np.ndarray, r_6_h: np.ndarray) -> tuple[float, float, float]:
    """The tool frame's mobile XYZ Euler angles (deg) in {0}: of ``0R_6 6R_H``, ``0R_6`` the
    last frame of the chain ``frames`` (the telemetry's ``tool_pose``)."""
    r = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            r[i, j] = (frames[5, 0, i] * r_6_h[0, j] + frames[5, 1, i] * r_6_h[1, j]
                       + frames[5, 2, i] * r_6_h[2, j])
    return euler_xyz_deg(r)


def warm_up() -> None:
    """Compile (or load from the cache) every kernel of this module for the argument types
    the controller and the simulator pass: a control loop must not pay a compilation at its
    first tick (100 ms and more). Called once, at import."""
    dh = np.zeros((6, 5))
    dh[:, 0] = 1.0
    q = np.zeros(6)
    frames = dh_frames(dh, q)
    pa = tool_point_axes(frames, np.eye(4), np.zeros(3))
    point_jacobian(frames, pa[3], pa[:3], True)
    point_jacobian(frames, frames[5, 3], np.eye(3), False)
    singularity_factors(frames, q, q, True, 0.0, 4)
    tool_euler_deg(frames, np.eye(3))
    euler_xyz_deg(np.eye(3))


warm_up()      # at import: before any device streams or loop runs
