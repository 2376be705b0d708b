"""The handpiece's step, compiled (numba): the motor's speed loop against the file's load,
its current limit and the current it reports, on arrays.

This kernel is the only implementation of the handpiece's laws (explained in
:mod:`dentibot.sim.handpiece`, whose :class:`~dentibot.sim.handpiece.HandpieceModel` calls
it). A handpiece is its state ``hs`` (:data:`STATE_FIELDS`), its constants ``hp``
(:data:`PARAM_FIELDS`) and a block of seeded current noise (A), refilled by its owner when
``hs[k]`` reaches the block's length (the kernel never draws random numbers).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: The handpiece's state (flags and modes as 0.0 / 1.0).
STATE_FIELDS = (
    "omega_rpm",        # file speed (rpm)
    "pos_deg",          # file position (deg)
    "cmd_rpm",          # commanded speed (rpm)
    "pos_mode",         # 1: a position move (move_relative) is running, 0: speed mode
    "target_deg",       # the move's target (deg)
    "move_rpm",         # the move's speed (rpm)
    "current_a",        # the current reading (A)
    "torque_mnm",       # signed torque the motor applies to the file (mNm)
    "stalled",          # the load exceeds the current limit's torque
    "current_limit_a",  # the drive's output current limit (A)
    "k",                # next sample of the noise block
    "t",                # time since start (s), for the reading's wander
)
#: The handpiece's constants.
PARAM_FIELDS = ("tau_s", "friction_current_a", "torque_per_amp_mnm", "current_offset_a",
                "current_wander_a", "current_wander_period_s", "wander_phase")

S = {name: i for i, name in enumerate(STATE_FIELDS)}
P = {name: i for i, name in enumerate(PARAM_FIELDS)}

(_W, _POS, _CMD, _POS_MODE, _TARGET, _MOVE_RPM, _CURRENT, _TORQUE, _STALLED, _LIMIT, _K,
 _T) = range(len(STATE_FIELDS))
_TAU, _I_FRICTION, _KT, _I_OFFSET, _I_WANDER, _WANDER_PERIOD, _WANDER_PHASE = range(
    len(PARAM_FIELDS))
#: Indices other kernels use (compiled constants).
S_OMEGA, S_TORQUE = _W, _TORQUE


@njit(cache=True)
def step(hs: np.ndarray, hp: np.ndarray, noise: np.ndarray, ts: float, resist_fwd_mnm: float,
         resist_rev_mnm: float) -> float:
    """Advance one period ``ts`` against a load resisting forward (positive) rotation with
    ``resist_fwd_mnm`` and reverse rotation with ``resist_rev_mnm`` (both >= 0, mNm at the
    file). Returns the file rotation this period (deg). ``noise[hs[k]]`` must exist."""
    tau = hp[_TAU]
    if hs[_POS_MODE] != 0.0:
        err = hs[_TARGET] - hs[_POS]
        ref = err / (6.0 * 4.0 * tau)  # P loop, deg -> rpm (1 rpm = 6 deg/s)
        m = hs[_MOVE_RPM]
        ref = min(max(ref, -m), m)
    else:
        ref = hs[_CMD]
    w = hs[_W]
    direction = w if abs(w) > 1e-6 else ref
    sgn = (direction > 0.0) - (direction < 0.0)
    resist = resist_fwd_mnm if sgn > 0 else resist_rev_mnm
    load = resist * sgn
    # the current limit covers the no-load current too (see the current model)
    t_max = max(0.0, hs[_LIMIT] - hp[_I_FRICTION]) * hp[_KT]
    a = -math.expm1(-ts / tau)   # exact discretisation of the first-order loop
    if resist > t_max and sgn != 0:
        hs[_STALLED] = 1.0
        w += (0.0 - w) * a
        hs[_TORQUE] = t_max * sgn if abs(w) > 1e-3 or ref != 0.0 else 0.0
    else:
        hs[_STALLED] = 0.0
        w += (ref - w) * a
        hs[_TORQUE] = load if (abs(w) > 1e-3 or ref != 0.0) else 0.0
    if abs(w) < 1e-6:
        w = 0.0
    hs[_W] = w
    dpos = w * 6.0 * ts
    hs[_POS] += dpos
    k = int(hs[_K])
    hs[_K] = k + 1
    fsgn = (w > 0.5) - (w < -0.5)
    current = hs[_TORQUE] / hp[_KT] + hp[_I_FRICTION] * fsgn + noise[k]
    if hp[_I_OFFSET] != 0.0 or hp[_I_WANDER] != 0.0:
        hs[_T] += ts
        current += hp[_I_OFFSET] + hp[_I_WANDER] * math.sin(
            2.0 * math.pi * hs[_T] / hp[_WANDER_PERIOD] + hp[_WANDER_PHASE])
    hs[_CURRENT] = current
    return dpos


def warm_up() -> None:
    """Compile (or load from the cache) the kernel (a simulator serving a real-time controller
    must not stall). Called once, at import."""
    hs = np.zeros(len(STATE_FIELDS))
    hp = np.ones(len(PARAM_FIELDS))
    step(hs, hp, np.zeros(4), 0.002, 1.0, 0.3)


warm_up()      # at import: before any device streams or loop runs
