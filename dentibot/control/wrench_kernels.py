"""Gravity compensation and the change of a wrench's frame, compiled (numba): eq 4.18 and
eq 4.26-4.31 on one reading.

:class:`~dentibot.control.wrench.GravityModel` and
:class:`~dentibot.control.wrench.WrenchTransform` fold their parameters into arrays (the
offset and the 6x3 gravity gain; the 6x6 {S} -> {H} map) and call these; so does the control
tick's estimate (:mod:`dentibot.control.tick_kernels`). They are the only implementation.
Units: N and N*m.

Compiled at import, as :mod:`~dentibot.control.kinematics_kernels` explains.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def gravity_wrench(gain: np.ndarray, e0: float, e1: float, e2: float) -> np.ndarray:
    """The tool's weight as a wrench in {S} (eq 4.15): ``gain @ e`` with ``e`` the third row
    of 0R_6 (the flange axes' z components in {0}) and ``gain`` the model's 6x3
    ``[-g Rz(th)^T; skew(r) (-g Rz(th)^T)]``."""
    out = np.empty(6)
    for i in range(6):
        out[i] = gain[i, 0] * e0 + gain[i, 1] * e1 + gain[i, 2] * e2
    return out


@njit(cache=True)
def external_wrench(measured: np.ndarray, offset: np.ndarray, gain: np.ndarray, e0: float,
                    e1: float, e2: float) -> np.ndarray:
    """The external wrench in {S} about the sensor origin (eq 4.18): the reading minus the
    offsets ``offset`` = (f0, tau0) minus :func:`gravity_wrench`."""
    g = gravity_wrench(gain, e0, e1, e2)
    out = np.empty(6)
    for i in range(6):
        out[i] = measured[i] - offset[i] - g[i]
    return out


@njit(cache=True)
def transform_wrench(matrix: np.ndarray, wrench: np.ndarray) -> np.ndarray:
    """``matrix @ wrench``: the wrench about the new reference point in the new axes (eq
    4.26-4.31, the 6x6 map of :class:`~dentibot.control.wrench.WrenchTransform`)."""
    out = np.empty(6)
    for i in range(6):
        s = 0.0
        for j in range(6):
            s += matrix[i, j] * wrench[j]
        out[i] = s
    return out


def warm_up() -> None:
    """Compile (or load from the cache) the kernels for the argument types the models pass:
    their parameters are read-only arrays (a type of their own to numba), the readings plain
    ones. Called once, at import."""
    from dentibot.control.linalg import readonly

    w = np.zeros(6)
    gain = readonly(np.zeros((6, 3)))
    gravity_wrench(gain, 0.0, 0.0, 1.0)
    external_wrench(w, readonly(w), gain, 0.0, 0.0, 1.0)
    transform_wrench(readonly(np.eye(6)), w)


warm_up()      # at import: before any device streams or loop runs
