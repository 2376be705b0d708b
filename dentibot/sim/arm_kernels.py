"""The Meca500's joint servo, compiled (numba): velocity and position modes, the command
queue, the trajectory filter's lag and gain, speed and joint limits, the wrist singularity.

This kernel is the only implementation of the arm's laws (explained in
:mod:`dentibot.sim.arm`, whose :class:`~dentibot.sim.arm.SimArmModel` calls it). An arm is
its state ``ast`` (:data:`STATE_FIELDS`), its joint arrays (``q``, ``qd``, ``vel_cmd``,
``target``: deg, deg/s), its constants ``ap`` (:data:`PARAM_FIELDS`) and joint limits
``lims`` (rows: lower, upper (deg), speed (deg/s)), and the queue of velocity commands
waiting in the robot (a ring: ``queue_t`` the times they take effect, ``queue_v`` their rates;
``ast``'s ``head`` and ``count``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: Meca500 error codes used here (programming manual, "error codes").
ERROR_JOINT_LIMIT = 1007
ERROR_SINGULARITY = 1012

#: The arm's modes, by their index in ``ast[mode]``.
MODES = ("idle", "vel", "pos")

#: The arm's state.
STATE_FIELDS = (
    "mode",             # index in MODES
    "vel_cmd_t",        # when the velocity command in force was given (s)
    "error_code",       # latched Meca500 error (0: none)
    "moving",           # a joint moved this step
    "pos_speed_scale",  # position mode's speed limit as a fraction of the joints' (SetJointVel)
    "head", "count",    # the command queue: its oldest entry, its length
)
#: The arm's constants (:class:`~dentibot.sim.arm.ArmParams`).
PARAM_FIELDS = ("servo_tau_s", "vel_timeout_s", "wrist_singularity_min", "rest_deg_s",
                "position_tau_s", "vel_gain")

S = {name: i for i, name in enumerate(STATE_FIELDS)}
P = {name: i for i, name in enumerate(PARAM_FIELDS)}

_MODE, _CMD_T, _ERROR, _MOVING, _POS_SCALE, _HEAD, _COUNT = range(len(STATE_FIELDS))
_SERVO_TAU, _VEL_TIMEOUT, _WRIST_MIN, _REST, _POS_TAU, _GAIN = range(len(PARAM_FIELDS))
_IDLE, _VEL, _POS = 0.0, 1.0, 2.0
#: Indices other kernels use (compiled constants).
S_MOVING = _MOVING


@njit(cache=True)
def fault(ast: np.ndarray, vel_cmd: np.ndarray, code: int) -> None:
    """Latch error ``code`` (the first one stays): the arm stops, its queue is dropped."""
    if ast[_ERROR] == 0.0:
        ast[_ERROR] = code
    ast[_MODE] = _IDLE
    vel_cmd[:] = 0.0
    ast[_HEAD] = 0.0
    ast[_COUNT] = 0.0


@njit(cache=True)
def command_velocity(ast: np.ndarray, lims: np.ndarray, vel_cmd: np.ndarray,
                     queue_t: np.ndarray, queue_v: np.ndarray, v: np.ndarray, t: float,
                     dead_time_s: float) -> bool:
    """MoveJointsVel at time ``t`` (s): the rates ``v`` (deg/s), each clipped to its joint's
    speed, in force now or, with a dead time, queued until ``t + dead_time_s``. False (and
    nothing done) when the queue is full: its owner grows it and calls again."""
    if dead_time_s > 0.0:
        cap = queue_t.shape[0]
        count = int(ast[_COUNT])
        if count == cap:
            return False
        if ast[_MODE] != _VEL:
            vel_cmd[:] = 0.0
            ast[_CMD_T] = t
        i = (int(ast[_HEAD]) + count) % cap
        queue_t[i] = t + dead_time_s
        dst = queue_v[i]
        ast[_COUNT] = count + 1
    else:
        dst = vel_cmd
        ast[_CMD_T] = t
    for j in range(6):
        m = lims[2, j]
        dst[j] = max(-m, min(m, v[j]))
    ast[_MODE] = _VEL
    return True


@njit(cache=True)
def step(ast: np.ndarray, ap: np.ndarray, lims: np.ndarray, q: np.ndarray, qd: np.ndarray,
         vel_cmd: np.ndarray, target: np.ndarray, queue_t: np.ndarray, queue_v: np.ndarray,
         t: float, ts: float) -> None:
    """Advance the servo one period ``ts`` to time ``t`` (s)."""
    ref = np.zeros(6)
    mode = ast[_MODE]
    if ast[_ERROR] != 0.0 or mode == _IDLE:
        pass
    elif mode == _VEL:
        cap = queue_t.shape[0]
        while ast[_COUNT] > 0.0 and queue_t[int(ast[_HEAD])] <= t + 1e-9:  # leaving the queue
            h = int(ast[_HEAD])
            ast[_CMD_T] = queue_t[h]
            vel_cmd[:] = queue_v[h]
            ast[_HEAD] = (h + 1) % cap
            ast[_COUNT] -= 1.0
        if t - ast[_CMD_T] <= ap[_VEL_TIMEOUT]:
            g = ap[_GAIN]
            for i in range(6):
                ref[i] = vel_cmd[i] if g == 1.0 else g * vel_cmd[i]
    else:
        k = 1.0 / max(ap[_POS_TAU], ts)
        s = max(ast[_POS_SCALE], 1e-6)
        scale = 0.0
        for i in range(6):
            ref[i] = (target[i] - q[i]) * k
            scale = max(scale, abs(ref[i]) / (lims[2, i] * s))
        if scale > 1.0:  # synchronous scaling: straight line in joint space
            for i in range(6):
                ref[i] = ref[i] / scale
    a = -math.expm1(-ts / ap[_SERVO_TAU])   # exact first-order discretisation
    moving = False
    new_q = np.empty(6)
    pos_mode = ast[_MODE] == _POS and ast[_ERROR] == 0.0
    for i in range(6):
        v = qd[i] + (ref[i] - qd[i]) * a
        m = lims[2, i]
        v = m if v > m else (-m if v < -m else v)  # noqa: FURB136 (NaN kept as the servo had it)
        if pos_mode:
            # never overshoot the target within one period
            rem = target[i] - q[i]
            if (v > 0.0 and v * ts > rem > 0.0) or (v < 0.0 and v * ts < rem < 0.0):
                v = rem / ts
        if abs(v) < 1e-9 or (ref[i] == 0.0 and abs(v) < ap[_REST]):
            v = 0.0
        else:
            moving = True
        qd[i] = v
        new_q[i] = q[i] + v * ts
    ast[_MOVING] = 1.0 if moving else 0.0
    if not moving:
        return
    for i in range(6):
        if new_q[i] < lims[0, i] or new_q[i] > lims[1, i]:
            new_q[i] = min(max(new_q[i], lims[0, i]), lims[1, i])
            fault(ast, vel_cmd, ERROR_JOINT_LIMIT)
    s_new = abs(math.sin(math.radians(new_q[4])))
    if ast[_MODE] == _VEL and s_new < ap[_WRIST_MIN] and \
            s_new < abs(math.sin(math.radians(q[4]))):
        # stop before entering the singular band (moving out of it is allowed)
        new_q[:] = q
        fault(ast, vel_cmd, ERROR_SINGULARITY)
    q[:] = new_q
    if ast[_ERROR] != 0.0:
        qd[:] = 0.0


def warm_up() -> None:
    """Compile (or load from the cache) the kernels (a simulator serving a real-time
    controller must not stall). Called once, at import."""
    ast = np.zeros(len(STATE_FIELDS))
    ast[_MODE] = _VEL
    ap = np.ones(len(PARAM_FIELDS))
    lims = np.array([[-10.0] * 6, [10.0] * 6, [1.0] * 6])
    z = np.zeros(6)
    step(ast, ap, lims, z.copy(), z.copy(), np.ones(6), z.copy(), np.zeros(4),
         np.zeros((4, 6)), 0.0, 0.002)
    command_velocity(ast, lims, z.copy(), np.zeros(4), np.zeros((4, 6)), z, 0.0, 0.016)


warm_up()      # at import: before any device streams or loop runs
