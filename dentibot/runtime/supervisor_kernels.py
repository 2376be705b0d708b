"""The supervisor's per-tick checks, compiled (numba): what is detected, over state arrays;
:class:`~dentibot.runtime.supervisor.Supervisor` and the observers of
:mod:`~dentibot.runtime.observers` keep those arrays, call these every tick, and word a
finding from the values a kernel reports only when it reports one. They are the only
implementation of each check.

Compiled at import, as :mod:`dentibot.control.kinematics_kernels` explains.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from dentibot.control.kinematics_kernels import singularity_factors

#: The input streams in the order the freshness state keeps them.
STREAMS = ("arm", "ft", "motor", "aux")
#: Fields of the freshness state, per stream: its last sequence number, the tick that number
#: arrived in, and whether one arrived yet.
FRESH_FIELDS = ("seq", "tick", "seen")
#: What :func:`inputs` reports in ``out``: each stream's age past its bound (-1: fresh), the
#: first non-finite value's group (0: none, 1 wrench, 2 joints, 3 motor), index and value,
#: the saturation flag and the force jump (-1: none).
INPUT_OUT_FIELDS = ("stale_arm", "stale_ft", "stale_motor", "stale_aux", "bad_group",
                    "bad_index", "bad_value", "saturated", "jump")
O_STALE, O_BAD_GROUP, O_BAD_INDEX, O_BAD_VALUE, O_SATURATED, O_JUMP = 0, 4, 5, 6, 7, 8
#: Bit of :attr:`~dentibot.io.interfaces.Wrench.status`: a channel is saturated (the
#: interfaces' WRENCH_SATURATED, which a test holds this to).
SATURATED_BIT = 0x1


@njit(cache=True)
def _fresh(fs: np.ndarray, i: int, seq: float, tick: float, bound: float) -> float:
    if fs[i, 2] == 0.0 or seq != fs[i, 0]:
        fs[i, 0], fs[i, 1], fs[i, 2] = seq, tick, 1.0
        return -1.0
    age = tick - fs[i, 1]
    return age if age > bound else -1.0


@njit(cache=True)
def inputs(fs: np.ndarray, bounds: np.ndarray, last_force: np.ndarray, tick: int,
           seq_arm: int, seq_ft: int, seq_motor: int, seq_aux: int, aux: bool,
           wrench: np.ndarray, q_deg: np.ndarray, current_a: float, velocity_rpm: float,
           position_deg: float, status: int, jump_limit_n: float, out: np.ndarray) -> bool:
    """The inputs' checks before anything is estimated: each stream's sequence number must
    change within its bound (in periods; ``fs`` one row per :data:`STREAMS`), every value
    finite (the first non-finite one is reported and the checks stop there), the saturation
    bit, and the largest change of a force component since the last sample against
    ``jump_limit_n`` (``last_force[3]`` is 1 once a force was kept). Writes
    :data:`INPUT_OUT_FIELDS` to ``out``; True when any of them is a finding."""
    found = False
    seqs = (seq_arm, seq_ft, seq_motor, seq_aux)
    for i in range(4):
        age = -1.0
        if i < 3 or aux:
            age = _fresh(fs, i, float(seqs[i]), float(tick), bounds[i])
        out[O_STALE + i] = age
        found = found or age >= 0.0
    out[O_BAD_GROUP] = 0.0
    out[O_SATURATED] = 0.0
    out[O_JUMP] = -1.0
    for i in range(6):
        if not math.isfinite(wrench[i]):
            out[O_BAD_GROUP], out[O_BAD_INDEX], out[O_BAD_VALUE] = 1.0, i, wrench[i]
            return True
    for i in range(6):
        if not math.isfinite(q_deg[i]):
            out[O_BAD_GROUP], out[O_BAD_INDEX], out[O_BAD_VALUE] = 2.0, i, q_deg[i]
            return True
    motor = (current_a, velocity_rpm, position_deg)
    for i in range(3):
        if not math.isfinite(motor[i]):
            out[O_BAD_GROUP], out[O_BAD_INDEX], out[O_BAD_VALUE] = 3.0, i, motor[i]
            return True
    if status & SATURATED_BIT:
        out[O_SATURATED] = 1.0
        found = True
    if last_force[3] != 0.0:
        jump = max(abs(wrench[0] - last_force[0]), abs(wrench[1] - last_force[1]),
                   abs(wrench[2] - last_force[2]))
        if jump > jump_limit_n:
            out[O_JUMP] = jump
            found = True
    last_force[0], last_force[1], last_force[2], last_force[3] = \
        wrench[0], wrench[1], wrench[2], 1.0
    return found


#: What :func:`estimate_checks` reports in ``out``: the F/T's file torque (mNm) and how far
#: the two sources are apart; the tip's lateral and axial position in the workspace box; the
#: three singularity factors.
ESTIMATE_OUT_FIELDS = ("tau_ft", "tau_diff", "lateral", "axial", "shoulder", "elbow",
                       "wrist")
E_TAU_FT, E_DIFF, E_LATERAL, E_AXIAL, E_SHOULDER, E_ELBOW, E_WRIST = range(7)
#: Bits of :func:`estimate_checks`' result (joint i out of range: ``JOINT_BIT << i``).
TORQUE_BIT, WORKSPACE_BIT, SHOULDER_BIT, ELBOW_BIT, WRIST_BIT, JOINT_BIT = 1, 2, 4, 8, 16, 32


@njit(cache=True)
def estimate_checks(disagree: np.ndarray, lim: np.ndarray, ts: float, turning: bool,
                    torque_mnm: float,
                    wrench_h5: float, boxed: bool, ox: float, oy: float, oz: float, ax: float,
                    ay: float, az: float, tx: float, ty: float, tz: float,
                    working_length_mm: float, q_deg: np.ndarray, q_lo: np.ndarray,
                    q_hi: np.ndarray, frames: np.ndarray, elbow_offset: float,
                    wrist_frame: int, out: np.ndarray) -> int:
    """The estimate's checks: the two file-torque sources apart by more than ``lim[0]`` mNm
    for longer than ``lim[1]`` s (``disagree[0]`` counts the periods of ``ts``; only while
    the file turns), the tip (tx, ty, tz) outside the workspace box around the orifice (o, axis a;
    ``boxed``: known), each joint within [q_lo, q_hi], and the singularity factors against
    their hard margins. ``lim``: (torque_mnm, torque_s, lateral_mm, above_mm,
    past_wl_mm, shoulder_min_mm, elbow_min, wrist_min). Writes
    :data:`ESTIMATE_OUT_FIELDS`; returns the bits of what was found (0: nothing)."""
    found = 0
    if turning:
        tau_ft = -1e3 * wrench_h5
        diff = abs(torque_mnm - tau_ft)
        out[E_TAU_FT], out[E_DIFF] = tau_ft, diff
        if diff > lim[0]:
            disagree[0] += 1.0
            if disagree[0] * ts > lim[1]:
                found |= TORQUE_BIT
        else:
            disagree[0] = 0.0
    else:
        disagree[0] = 0.0
    if boxed:
        d0, d1, d2 = tx - ox, ty - oy, tz - oz
        axial = d0 * ax + d1 * ay + d2 * az
        lateral = math.sqrt(max(0.0, d0 * d0 + d1 * d1 + d2 * d2 - axial * axial))
        out[E_LATERAL], out[E_AXIAL] = lateral, axial
        if lateral > lim[2] or axial < -lim[3] or axial > working_length_mm + lim[4]:
            found |= WORKSPACE_BIT
    for i in range(6):
        if q_deg[i] < q_lo[i] or q_deg[i] > q_hi[i]:
            found |= JOINT_BIT << i
    s = singularity_factors(frames, q_deg, np.zeros(6), False, elbow_offset, wrist_frame)
    out[E_SHOULDER], out[E_ELBOW], out[E_WRIST] = s[0], s[1], s[2]
    if s[0] < lim[5]:
        found |= SHOULDER_BIT
    if s[1] < lim[6]:
        found |= ELBOW_BIT
    if s[2] < lim[7]:
        found |= WRIST_BIT
    return found


#: Bit of :func:`command_checks`' result: the tip's commanded speed above the cap (joint i
#: above its limit: bit i).
TIP_SPEED_BIT = 1 << 6


@njit(cache=True)
def command_checks(qdot_deg_s: np.ndarray, twist: np.ndarray, speed_limits: np.ndarray,
                   tooth: bool, tooth_twist: np.ndarray, cap_mm_s: float,
                   out: np.ndarray) -> int:
    """The command's checks: each joint rate against its limit (bit i), and the tip's
    commanded speed (relative to the tracked tooth's when ``tooth``) against the cap
    (:data:`TIP_SPEED_BIT`), written to ``out[0]``. Returns the bits (0: nothing)."""
    found = 0
    for i in range(6):
        if abs(qdot_deg_s[i]) > speed_limits[i] * (1.0 + 1e-9):
            found |= 1 << i
    r0, r1, r2 = twist[0], twist[1], twist[2]
    if tooth:
        r0, r1, r2 = r0 - tooth_twist[0], r1 - tooth_twist[1], r2 - tooth_twist[2]
    v = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
    out[0] = v
    if v > cap_mm_s:
        found |= TIP_SPEED_BIT
    return found


#: The spindle observer's state: periods since the file command changed, consecutive
#: periods off the command, and the speed tolerance last applied (rpm).
SPINDLE_FIELDS = ("since", "bad", "tol")
SP_SINCE, SP_BAD, SP_TOL = range(3)
#: :func:`spindle`'s findings.
SPINDLE_DISABLED, SPINDLE_SPEED = 1, 2


@njit(cache=True)
def spindle(st: np.ndarray, lim: np.ndarray, ts: float, changed: bool, compared: bool,
            want_rpm: float, rpm: float, enabled: bool, torque_mnm: float) -> int:
    """One period of the handpiece against its command (see
    :class:`~dentibot.runtime.observers.SpindleObserver`): ``changed``, a new command
    (the counts restart); ``compared``, a command whose speed is compared (not a reversal);
    ``want_rpm`` its speed (0 for a stop). ``lim``: (settle_s, tolerance_rpm,
    tolerance_share, loaded_mnm, persist_s). Returns 0, :data:`SPINDLE_DISABLED` or
    :data:`SPINDLE_SPEED` (the tolerance in ``st``)."""
    if changed:
        st[SP_SINCE] = st[SP_BAD] = 0.0
    st[SP_SINCE] += 1.0
    if not compared or st[SP_SINCE] * ts < lim[0]:
        return 0
    if want_rpm != 0.0 and not enabled:
        return SPINDLE_DISABLED
    tol = max(lim[1], lim[2] * abs(want_rpm))
    st[SP_TOL] = tol
    slow_under_load = abs(rpm) < abs(want_rpm) and abs(torque_mnm) > lim[3]
    if abs(rpm - want_rpm) > tol and not slow_under_load:
        st[SP_BAD] += 1.0
    else:
        st[SP_BAD] = 0.0
    return SPINDLE_SPEED if st[SP_BAD] * ts >= lim[4] else 0


#: The fracture observer's state: the learnt free-running torque and how many samples it is
#: the mean of; the window's ring (its oldest slot, how many samples it holds).
FRACTURE_FIELDS = ("free_mnm", "free_n", "head", "count")
F_FREE, F_FREE_N, F_HEAD, F_COUNT = range(4)


@njit(cache=True)
def fracture(st: np.ndarray, ring: np.ndarray, lim: np.ndarray, n_recent: int,
             at_speed: bool, torque_mnm: float, depth_mm: float, depth_known: bool,
             out: np.ndarray) -> bool:
    """One sample of the fracture signature (see
    :class:`~dentibot.runtime.observers.FractureObserver`): ``ring`` holds the window's
    (torque, depth, depth known) rows; ``lim``: (loaded_mnm, share, free_band_mnm,
    min_depth_mm, withdraw_mm). True (the loaded and the recent mean in ``out``, the window
    emptied) when a fracture is suspected."""
    n = ring.shape[0]
    if not at_speed:
        st[F_HEAD] = st[F_COUNT] = 0.0
        return False
    if depth_known and depth_mm < -1.0 and st[F_FREE_N] < 10_000:
        st[F_FREE_N] += 1.0
        st[F_FREE] += (torque_mnm - st[F_FREE]) / st[F_FREE_N]
    head, count = int(st[F_HEAD]), int(st[F_COUNT])
    if count < n:
        slot = (head + count) % n
        count += 1
    else:                              # full: the oldest goes
        slot = head
        head = (head + 1) % n
    ring[slot, 0], ring[slot, 1], ring[slot, 2] = torque_mnm, depth_mm, depth_known
    st[F_HEAD], st[F_COUNT] = head, count
    if count < n or not depth_known or depth_mm < lim[3] or ring[head, 2] == 0.0 \
            or depth_mm < ring[head, 1] - lim[4]:
        return False
    n_ref = n - n_recent
    ref = 0.0
    for j in range(n_ref):
        ref += ring[(head + j) % n, 0]
    recent = 0.0
    for j in range(n_ref, n):
        recent += ring[(head + j) % n, 0]
    loaded = ref / n_ref - st[F_FREE]
    now = recent / n_recent - st[F_FREE]
    if loaded >= lim[0] and now <= min(lim[1] * loaded, lim[2]):
        out[0], out[1] = loaded, now
        st[F_HEAD] = st[F_COUNT] = 0.0
        return True
    return False


#: The tip-speed observer's state: the ring's oldest slot and fill, the ticks above the bound.
TIP_FIELDS = ("head", "count", "bad")
T_HEAD, T_COUNT, T_BAD = range(3)


@njit(cache=True)
def tip_speed(st: np.ndarray, ring: np.ndarray, x: float, y: float, z: float, ts: float,
              bound_mm_s: float) -> float:
    """One tip position (mm, {0}) into the window ``ring`` (rows x, y, z); the speed from the
    window's first to its last position (-1 until two are in), and the count of consecutive
    ticks above ``bound_mm_s`` kept in ``st``."""
    n = ring.shape[0]
    head, count = int(st[T_HEAD]), int(st[T_COUNT])
    if count < n:
        slot = (head + count) % n
        count += 1
    else:
        slot = head
        head = (head + 1) % n
    ring[slot, 0], ring[slot, 1], ring[slot, 2] = x, y, z
    st[T_HEAD], st[T_COUNT] = head, count
    if count < 2:
        return -1.0
    d0, d1, d2 = x - ring[head, 0], y - ring[head, 1], z - ring[head, 2]
    v = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) / ((count - 1) * ts)
    st[T_BAD] = st[T_BAD] + 1.0 if v > bound_mm_s else 0.0
    return v


def warm_up() -> None:
    """Compile (or load from the cache) the kernels for the argument types the supervisor
    passes. Called once, at import."""
    from dentibot.control.kinematics_kernels import dh_frames

    z6 = np.zeros(6)
    inputs(np.zeros((4, 3)), np.full(4, 10.0), np.zeros(4), 0, 0, 0, 0, 0, True, z6, z6, 0.0,
           0.0, 0.0, 0, 15.0, np.zeros(len(INPUT_OUT_FIELDS)))
    dh = np.zeros((6, 5))
    dh[:, 0] = 1.0
    estimate_checks(np.zeros(1), np.ones(8), 0.002, True, 0.0, 0.0, True, 0.0, 0.0, 0.0, 0.0, 0.0,
                    1.0, 0.0, 0.0, 0.0, 16.0, z6, z6 - 1.0, z6 + 1.0, dh_frames(dh, z6), 0.0,
                    4, np.zeros(len(ESTIMATE_OUT_FIELDS)))
    command_checks(z6, z6, z6 + 1.0, False, z6, 50.0, np.zeros(1))
    fracture(np.zeros(len(FRACTURE_FIELDS)), np.zeros((23, 3)), np.ones(5), 3, True, 1.0, 2.0,
             True, np.zeros(2))
    tip_speed(np.zeros(len(TIP_FIELDS)), np.zeros((6, 3)), 0.0, 0.0, 0.0, 0.002, 60.0)
    spindle(np.zeros(len(SPINDLE_FIELDS)), np.ones(5), 0.002, True, True, 60.0, 60.0, True,
            0.0)


warm_up()      # at import: before any device streams or loop runs
