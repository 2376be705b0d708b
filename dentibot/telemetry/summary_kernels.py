"""A run summary's figures over a block of ticks, compiled (numba).

:meth:`~dentibot.telemetry.summary.SummaryAccumulator.add_block` takes the compiled drilling
ticks' rows 25 to 256 at a time; over so few numbers, numpy's per-call dispatch (a dozen
calls) costs ten times the arithmetic. :func:`block_figures` walks the block once, with the
operations :meth:`~dentibot.telemetry.summary.SummaryAccumulator.add` applies row by row, in
the same order, so the summary is the same to the last bit.

Compiled (or loaded from numba's cache) when the module is imported (:func:`warm_up`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: :func:`block_figures`' running sums (``sums``): the run's and the step's duration (s),
#: the run's and the step's sum of |file torque| while the file turns (mNm)
DURATION_RUN, DURATION_STEP, TORQUE_RUN, TORQUE_STEP = range(4)


@njit(cache=True)
def block_figures(cols, depth_col, torque_col, rpm_col, force_col, k0, ts, prev_t, sums):
    """Figures of the ticks ``k0, k0 + 1, ...`` whose rows are ``cols``: returns ``(depth
    max, |torque| max, force norm max, ticks turning, the last tick's t)``, and adds each
    tick's duration (``t - prev_t``, at least 0, with ``t = k ts``) and |torque| while the
    motor turns to ``sums`` one by one. Every value must be finite (the caller checks)."""
    depth_max = -math.inf
    torque_max = -math.inf
    force_max = -math.inf
    turning = 0
    for i in range(cols.shape[0]):
        t = (k0 + i) * ts
        dt = t - prev_t
        dt = max(dt, 0.0)
        prev_t = t
        sums[DURATION_RUN] += dt
        sums[DURATION_STEP] += dt
        depth = cols[i, depth_col]
        depth_max = max(depth_max, depth)
        tau = abs(cols[i, torque_col])
        torque_max = max(torque_max, tau)
        if cols[i, rpm_col] != 0.0:
            sums[TORQUE_RUN] += tau
            sums[TORQUE_STEP] += tau
            turning += 1
        fx, fy, fz = cols[i, force_col], cols[i, force_col + 1], cols[i, force_col + 2]
        force = math.sqrt(fx * fx + fy * fy + fz * fz)
        force_max = max(force_max, force)
    return depth_max, torque_max, force_max, turning, prev_t


@njit(cache=True)
def all_finite(cols, columns) -> bool:
    """Whether every row of ``cols`` is finite in each of ``columns``."""
    for i in range(cols.shape[0]):
        for j in columns:
            if not math.isfinite(cols[i, j]):
                return False
    return True


def warm_up() -> None:
    """Compile (or load) the kernels for the types a block carries."""
    cols = np.zeros((1, 4))
    block_figures(cols, 0, 1, 2, 1, 0, 0.002, 0.0, np.zeros(4))
    all_finite(cols, np.arange(2, dtype=np.intp))


warm_up()
