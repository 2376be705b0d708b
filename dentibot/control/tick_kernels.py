"""Step 2 of the control tick, compiled (numba): from the joint angles, the raw sensor
reading and the motor's current to the chain, the tool Jacobian, the external wrench at the
reference point, the file torque and the tip, in one call.

:func:`dentibot.control.tick.sense` calls it for the runtime and the benchmark; it composes
the kernels of :mod:`~dentibot.control.kinematics_kernels` (the chain, eq 3.1-3.14),
:mod:`~dentibot.control.wrench_kernels` (eq 4.18, 4.26-4.31) and
:func:`~dentibot.control.feedrate.file_torque_estimate_mnm` (eq 5.4-5.5), which stay the only
implementation of each law.

Compiled at import, as :mod:`~dentibot.control.kinematics_kernels` explains.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from dentibot.control.feedrate import (
    GEAR_RATIO,
    KM_MNM_PER_A,
    MOVING_RPM,
    file_torque_estimate_mnm,
)
from dentibot.control.kinematics_kernels import dh_frames, point_jacobian, tool_point_axes
from dentibot.control.wrench_kernels import external_wrench, transform_wrench


@njit(cache=True)
def sense(q_deg: np.ndarray, raw: np.ndarray, current_a: float, velocity_rpm: float,
          dh: np.ndarray, tool: np.ndarray, ref_h: np.ndarray, compensate: bool,
          offset: np.ndarray, gain: np.ndarray, to_h: np.ndarray, efficiency: float,
          friction_current_a: float):
    """One tick's estimate at the joint angles ``q_deg`` (deg) with the raw reading ``raw``
    (N, N*m, {S}) and the motor's current and speed.

    ``dh``, ``tool`` (6T_H) and ``ref_h`` (the reference point in {H}, mm) as the kinematics
    kernels take them; with ``compensate``, the gravity model's ``offset`` and ``gain`` and
    the {S} -> {H} map ``to_h`` give the external wrench at the reference point (zero
    without). Returns ``(frames, J_H, wrench_h, |f|, file torque mNm, tip axes)`` where the
    last is :func:`tool_point_axes` at the tip (rows x_H, y_H, z_H, tip; {0})."""
    frames = dh_frames(dh, q_deg)
    pa = tool_point_axes(frames, tool, ref_h)
    jh = point_jacobian(frames, pa[3], pa[:3], True)
    if compensate:
        ws = external_wrench(raw, offset, gain, frames[5, 0, 2], frames[5, 1, 2],
                             frames[5, 2, 2])
        wrench_h = transform_wrench(to_h, ws)
    else:
        wrench_h = np.zeros(6)
    norm = 0.0
    for i in range(6):
        norm += wrench_h[i] * wrench_h[i]
    tau = file_torque_estimate_mnm(current_a, velocity_rpm, efficiency, friction_current_a,
                                   KM_MNM_PER_A, GEAR_RATIO, MOVING_RPM)
    if ref_h[0] == 0.0 and ref_h[1] == 0.0 and ref_h[2] == 0.0:
        tip = pa                        # the reference point is the tip (self-alignment)
    else:
        tip = tool_point_axes(frames, tool, np.zeros(3))
    return frames, jh, wrench_h, math.sqrt(norm), tau, tip


def warm_up() -> None:
    """Compile (or load from the cache) :func:`sense` for the argument types the runtime
    passes: the gravity model's and the transform's arrays are read-only, and so are the
    stand-ins :func:`dentibot.control.tick.sense` passes before a model is known. Called
    once, at import."""
    from dentibot.control.linalg import readonly

    dh = np.zeros((6, 5))
    dh[:, 0] = 1.0
    z6 = np.zeros(6)
    sense(z6, z6, 0.0, 0.0, dh, np.eye(4), np.zeros(3), True, readonly(z6),
          readonly(np.zeros((6, 3))), readonly(np.eye(6)), 1.0, 0.0)


warm_up()      # at import: before any device streams or loop runs
