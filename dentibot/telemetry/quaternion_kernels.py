"""The 3D view's rotations, compiled (numba): the only implementation of them.

Quaternions are ``(x, y, z, w)`` tuples, unit, Hamilton's product. The rows' poses carry
mobile XYZ Euler angles in degrees (``R = Rx(alpha) Ry(beta) Rz(gamma)``,
docs/architecture.md). :mod:`dentibot.telemetry.foxglove` calls the scalar functions for one
row (the live view, a row recorded alone); :func:`fill_tool_frames` runs the same functions
over a block of ticks and writes the frames' numbers straight into the block's ``/tf``
messages (:class:`~dentibot.telemetry.tf_cdr.TfEncoder`), so a block is recorded bit for bit
as its rows would be.

The kernels are compiled (or loaded from numba's cache) when the module is imported
(:func:`warm_up`): the recorder's writer must not pay a compilation at its first block.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: metres per millimetre (the 3D panel works in metres)
MM = 0.001


@njit(cache=True)
def quat_from_euler_xyz_deg(alpha: float, beta: float, gamma: float):
    """Unit quaternion of ``R = Rx(alpha) Ry(beta) Rz(gamma)`` (degrees): the product of
    the three axis quaternions, written out."""
    ha, hb, hg = math.radians(alpha) * 0.5, math.radians(beta) * 0.5, math.radians(gamma) * 0.5
    ca, sa = math.cos(ha), math.sin(ha)
    cb, sb = math.cos(hb), math.sin(hb)
    cg, sg = math.cos(hg), math.sin(hg)
    # qx(a) * qy(b) = (sa cb, ca sb, sa sb, ca cb); then * qz(g)
    x1, y1, z1, w1 = sa * cb, ca * sb, sa * sb, ca * cb
    return (x1 * cg + y1 * sg, y1 * cg - x1 * sg, z1 * cg + w1 * sg, w1 * cg - z1 * sg)


@njit(cache=True)
def qmul(a, b):
    """Hamilton's product ``a b``."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz)


@njit(cache=True)
def qconj(q):
    return (-q[0], -q[1], -q[2], q[3])


@njit(cache=True)
def qrotate(q, v):
    """``v`` rotated by the unit quaternion ``q``: v + 2 w (u x v) + 2 u x (u x v)."""
    x, y, z, w = q
    vx, vy, vz = v
    tx, ty, tz = 2.0 * (y * vz - z * vy), 2.0 * (z * vx - x * vz), 2.0 * (x * vy - y * vx)
    return (vx + w * tx + y * tz - z * ty, vy + w * ty + z * tx - x * tz,
            vz + w * tz + x * ty - y * tx)


@njit(cache=True)
def flange_of_tip(p_0h, q_0h, q_6h, p_6h):
    """The flange in {0} from the tip's pose and the tool geometry 6T_H:
    0T_6 = 0T_H (6T_H)^-1. Returns (position in mm, rotation)."""
    q_06 = qmul(q_0h, qconj(q_6h))
    r = qrotate(q_06, p_6h)
    return (p_0h[0] - r[0], p_0h[1] - r[1], p_0h[2] - r[2]), q_06


@njit(cache=True)
def fill_tool_frames(buf, tool, q_6h, p_6h, with_tool: bool, word: int) -> None:
    """Row ``i`` of ``buf`` (float64 words of a ``/tf`` message per row) gets, from word
    ``word`` on, the frame the tool pose ``tool[i]`` (x, y, z mm, Euler deg) places: the
    flange (``with_tool``, from the geometry ``q_6h``, ``p_6h``) or else the file tip, as
    seven numbers: position in metres, then the quaternion."""
    for i in range(tool.shape[0]):
        p_0h = (tool[i, 0], tool[i, 1], tool[i, 2])
        q = quat_from_euler_xyz_deg(tool[i, 3], tool[i, 4], tool[i, 5])
        p = p_0h
        if with_tool:
            p, q = flange_of_tip(p_0h, q, q_6h, p_6h)
        buf[i, word] = p[0] * MM
        buf[i, word + 1] = p[1] * MM
        buf[i, word + 2] = p[2] * MM
        buf[i, word + 3] = q[0]
        buf[i, word + 4] = q[1]
        buf[i, word + 5] = q[2]
        buf[i, word + 6] = q[3]


def warm_up() -> None:
    """Compile (or load) every kernel for the types it is called with."""
    q = quat_from_euler_xyz_deg(1.0, 2.0, 3.0)
    qrotate(qmul(q, qconj(q)), (1.0, 2.0, 3.0))
    flange_of_tip((1.0, 2.0, 3.0), q, q, (0.0, 0.0, 1.0))
    buf = np.zeros((1, 8))
    fill_tool_frames(buf, np.zeros((1, 6)), q, (0.0, 0.0, 1.0), True, 0)
    fill_tool_frames(buf, np.zeros((1, 6)), q, (0.0, 0.0, 1.0), False, 0)


warm_up()
